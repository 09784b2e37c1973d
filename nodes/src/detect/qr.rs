//! `detect.qr_finder`: QR-code finder patterns (the three concentric squares in a code's corners).
//!
//! [`qr_finders`] binarizes the image, scans rows for the 1:1:3:1:1 dark–light–dark–light–dark
//! run-length signature, confirms each hit by vertical, horizontal (again) and diagonal cross-
//! checks through the candidate centre, and clusters the confirmed centres. [`QrFinder`] is the
//! thin operator around it. Sequential and deterministic.

use std::sync::Arc;

use ocellus_engine::op::{Inputs, Op, OpError, Operator, Outputs, PortSpec, RunContext};
use ocellus_engine::params;
use ocellus_engine::types::PortType;
use ocellus_engine::value::{Metrics, Value};

use super::gray::gray_u8;

params! {
    /// Parameters of `detect.qr_finder`.
    pub struct QrFinderParams {
        /// Binarization threshold (0–255 gray levels): darker pixels are dark. -1 (default) picks
        /// it with Otsu's method.
        threshold: i32 = -1 => [min = -1, max = 255],
        /// Largest allowed deviation of each run from its ideal length, as a fraction of the
        /// module size (run "3" allows three times as much). Default 0.5 (ZXing's).
        tolerance: f64 = 0.5 => [min = 0.05, max = 1.0],
        /// Confirmations (rows whose scan hit the same pattern) a centre needs to be reported.
        /// Default 2.
        min_confirmations: u32 = 2 => [min = 1],
    }
}

/// A confirmed finder pattern.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Finder {
    /// Centre column (pixel centres at integers).
    pub x: f64,
    /// Centre row.
    pub y: f64,
    /// Module size in pixels (the pattern is 7 modules wide).
    pub module: f64,
    /// Number of row scans that confirmed it.
    pub count: u32,
}

/// Otsu's threshold of an 8-bit histogram: the `t` maximizing the between-class variance of
/// `{v ≤ t}` and `{v > t}` (the first on ties).
pub fn otsu_threshold(gray: &[u8]) -> u8 {
    let mut hist = [0u64; 256];
    for &v in gray {
        hist[v as usize] += 1;
    }
    let total = gray.len() as f64;
    let sum_all: f64 = hist
        .iter()
        .enumerate()
        .map(|(i, &c)| i as f64 * c as f64)
        .sum();
    let (mut w0, mut sum0) = (0.0, 0.0);
    let (mut best, mut best_t) = (-1.0, 0u8);
    for (t, &c) in hist.iter().enumerate() {
        w0 += c as f64;
        sum0 += t as f64 * c as f64;
        let w1 = total - w0;
        if w0 == 0.0 || w1 == 0.0 {
            continue;
        }
        let d = sum0 / w0 - (sum_all - sum0) / w1;
        let var = w0 * w1 * d * d;
        if var > best {
            best = var;
            best_t = t as u8;
        }
    }
    best_t
}

/// True when five run lengths match 1:1:3:1:1 within `tol` modules.
fn ratio_ok(c: &[u32; 5], tol: f64) -> bool {
    let total: u32 = c.iter().sum();
    if total < 7 || c.contains(&0) {
        return false;
    }
    let m = f64::from(total) / 7.0;
    let v = m * tol;
    let ok = |n: u32, k: f64| (f64::from(n) - k * m).abs() < k * v;
    ok(c[0], 1.0) && ok(c[1], 1.0) && ok(c[2], 3.0) && ok(c[3], 1.0) && ok(c[4], 1.0)
}

/// Binary image: `true` = dark.
struct Binary<'a> {
    dark: &'a [bool],
    width: usize,
    height: usize,
}

impl Binary<'_> {
    fn at(&self, x: isize, y: isize) -> Option<bool> {
        if x < 0 || y < 0 || x >= self.width as isize || y >= self.height as isize {
            None
        } else {
            Some(self.dark[y as usize * self.width + x as usize])
        }
    }

    /// Run lengths through `(x, y)` along `(dx, dy)`: the dark run holding the centre and the
    /// light, dark runs on both sides, each at most `max_run` steps. Returns the runs and the
    /// centre's offset (in steps, from `(x, y)`) of the middle run.
    fn cross(
        &self,
        x: isize,
        y: isize,
        dx: isize,
        dy: isize,
        max_run: u32,
    ) -> Option<([u32; 5], f64)> {
        if self.at(x, y) != Some(true) {
            return None;
        }
        let mut c = [0u32; 5];
        // Backwards: centre dark (c[2]), light (c[1]), dark (c[0]).
        let walk = |sign: isize, slots: [usize; 3], c: &mut [u32; 5]| -> Option<isize> {
            let mut k = 0isize;
            for (s, want) in slots.into_iter().zip([true, false, true]) {
                loop {
                    let (px, py) = (x + sign * k * dx, y + sign * k * dy);
                    match self.at(px, py) {
                        Some(v) if v == want => {
                            c[s] += 1;
                            k += 1;
                            if c[s] > max_run && s != 2 {
                                return None;
                            }
                        }
                        Some(_) => break,
                        None => {
                            if s == slots[2] && c[s] > 0 {
                                break;
                            }
                            return None;
                        }
                    }
                }
                if c[s] == 0 {
                    return None;
                }
            }
            Some(k)
        };
        walk(-1, [2, 1, 0], &mut c)?;
        // The centre pixel was counted once going backwards; forwards starts past it.
        let centre_back = c[2];
        let mut fwd = [0u32; 5];
        {
            let mut k = 1isize;
            for (s, want) in [2usize, 3, 4].into_iter().zip([true, false, true]) {
                loop {
                    let (px, py) = (x + k * dx, y + k * dy);
                    match self.at(px, py) {
                        Some(v) if v == want => {
                            fwd[s] += 1;
                            k += 1;
                            if fwd[s] > max_run && s != 2 {
                                return None;
                            }
                        }
                        Some(_) => break,
                        None => {
                            if s == 4 && fwd[s] > 0 {
                                break;
                            }
                            return None;
                        }
                    }
                }
                if s != 2 && fwd[s] == 0 {
                    return None;
                }
            }
        }
        c[2] += fwd[2];
        c[3] = fwd[3];
        c[4] = fwd[4];
        // Middle run spans offsets -(centre_back - 1) ..= fwd[2].
        let first = -(centre_back as f64 - 1.0);
        let last = f64::from(fwd[2]);
        Some((c, (first + last) / 2.0))
    }
}

/// Finder-pattern centres of a gray 8-bit image, most-confirmed first (ties by row, then
/// column). `threshold` `None` uses Otsu's. See [`QrFinder::DOC`](Op::DOC).
///
/// # Panics
///
/// If `gray.len() != width × height`.
pub fn qr_finders(
    gray: &[u8],
    width: usize,
    height: usize,
    threshold: Option<u8>,
    tolerance: f64,
    min_confirmations: u32,
) -> Vec<Finder> {
    assert_eq!(gray.len(), width * height, "gray buffer size");
    if gray.is_empty() {
        return Vec::new();
    }
    let t = threshold.unwrap_or_else(|| otsu_threshold(gray));
    let dark: Vec<bool> = gray.iter().map(|&v| v <= t).collect();
    let bin = Binary {
        dark: &dark,
        width,
        height,
    };
    // Clusters: (sum x, sum y, sum module, count).
    let mut clusters: Vec<(f64, f64, f64, u32)> = Vec::new();
    for y in 0..height {
        let row = &dark[y * width..(y + 1) * width];
        // Runs of the row: (start, length, dark).
        let mut runs: Vec<(usize, u32, bool)> = Vec::new();
        for (x, &d) in row.iter().enumerate() {
            match runs.last_mut() {
                Some(r) if r.2 == d => r.1 += 1,
                _ => runs.push((x, 1, d)),
            }
        }
        for w in runs.windows(5) {
            if !w[0].2 {
                continue;
            }
            let c = [w[0].1, w[1].1, w[2].1, w[3].1, w[4].1];
            if !ratio_ok(&c, tolerance) {
                continue;
            }
            let total: u32 = c.iter().sum();
            let cx = w[2].0 as f64 + (f64::from(w[2].1) - 1.0) / 2.0;
            if let Some((x, yc, module)) = confirm(&bin, cx, y as f64, total, tolerance) {
                let found = clusters.iter_mut().find(|cl| {
                    let n = f64::from(cl.3);
                    let (mx, my, mm) = (cl.0 / n, cl.1 / n, cl.2 / n);
                    (mx - x).abs() <= mm
                        && (my - yc).abs() <= mm
                        && (module - mm).abs() <= mm.max(1.0)
                });
                match found {
                    Some(cl) => {
                        cl.0 += x;
                        cl.1 += yc;
                        cl.2 += module;
                        cl.3 += 1;
                    }
                    None => clusters.push((x, yc, module, 1)),
                }
            }
        }
    }
    let mut out: Vec<Finder> = clusters
        .into_iter()
        .filter(|c| c.3 >= min_confirmations)
        .map(|c| {
            let n = f64::from(c.3);
            Finder {
                x: c.0 / n,
                y: c.1 / n,
                module: c.2 / n,
                count: c.3,
            }
        })
        .collect();
    out.sort_by(|a, b| {
        b.count
            .cmp(&a.count)
            .then(a.y.total_cmp(&b.y))
            .then(a.x.total_cmp(&b.x))
    });
    out
}

/// Vertical, horizontal and diagonal cross-checks of a row hit at column `cx` of row `y` whose
/// runs total `total`; the refined centre and module size.
fn confirm(bin: &Binary<'_>, cx: f64, y: f64, total: u32, tol: f64) -> Option<(f64, f64, f64)> {
    let max_run = total;
    let similar = |t: u32| 5 * t.abs_diff(total) < 2 * total;
    let xi = cx.round() as isize;
    let (cv, off_y) = bin.cross(xi, y as isize, 0, 1, max_run)?;
    let tv: u32 = cv.iter().sum();
    if !ratio_ok(&cv, tol) || !similar(tv) {
        return None;
    }
    let yc = y + off_y;
    let (ch, off_x) = bin.cross(xi, yc.round() as isize, 1, 0, max_run)?;
    let th: u32 = ch.iter().sum();
    if !ratio_ok(&ch, tol) || !similar(th) {
        return None;
    }
    let xc = xi as f64 + off_x;
    let (cd, _) = bin.cross(xc.round() as isize, yc.round() as isize, 1, 1, max_run)?;
    if !ratio_ok(&cd, tol * 1.5) {
        return None;
    }
    let module = f64::from(th + tv) / 14.0;
    Some((xc, yc, module))
}

/// QR finder-pattern detector (`detect.qr_finder`). See [`qr_finders`].
#[derive(Debug, Clone, PartialEq)]
pub struct QrFinder {
    threshold: Option<u8>,
    tolerance: f64,
    min_confirmations: u32,
}

impl Op for QrFinder {
    type Params = QrFinderParams;
    const ID: &'static str = "detect.qr_finder";
    const SUMMARY: &'static str =
        "Finds QR-code finder patterns (1:1:3:1:1 concentric squares) and returns their centres.";
    const DOC: &'static str = r#"
Locates the finder patterns of QR codes: the 7×7-module squares (dark ring, light ring, dark
3×3 core) in three corners of every code. The method is ZXing's finder-pattern scan:

1. Binarize: a pixel is dark when its gray value is ≤ `threshold` (Otsu's threshold when -1).
2. Scan every row for five consecutive runs dark, light, dark, light, dark whose lengths match
   1:1:3:1:1: each run may deviate from its ideal length by `tolerance` × the module size
   (total / 7), three times that for the core.
3. Cross-check through the candidate centre: the vertical runs must match the ratio with a
   total within 40 % of the row's (their middle gives the centre row), then the horizontal runs
   again at that row (their middle gives the centre column), then the diagonal runs (ratio
   only, 1.5 × tolerance).
4. Cluster confirmed centres: a hit within one module (in x, y and size) of a cluster's mean
   joins it. Clusters with at least `min_confirmations` hits are reported at their mean.

Coordinates: pixel centres at integers. Rotated codes work because lines through a finder's
centre cross the rings in the same proportions (the diagonal check tolerates more).

Input: any image; colour is reduced to BT.601 luma, u16 to v/257 and f32 to clamp(v,0,1)·255.

Outputs: `centres` (Points2D, most-confirmed first, ties by row then column) and `metrics`:
`count` (centres reported) and `module_size` (mean module size in pixels, 0 if none).

OpenCV's `QRCodeDetector` uses the same signature but then fits whole codes; this operator
stops at the finder patterns (no decoding, no grouping into codes).

Reference: ZXing, `FinderPatternFinder` (core/src/main/java/com/google/zxing/qrcode/detector);
ISO/IEC 18004 (finder pattern geometry).

Example (a node of a graph):
    "finders": (op: "detect.qr_finder", inputs: { "image": "frame.image" },
                params: (threshold: -1, tolerance: 0.5)),
"#;

    fn inputs() -> Vec<PortSpec> {
        vec![PortSpec::new(
            "image",
            PortType::Image,
            "image, any format (colour reduced to luma, depth scaled to 0–255)",
        )]
    }

    fn outputs() -> Vec<PortSpec> {
        vec![
            PortSpec::new(
                "centres",
                PortType::Points2D,
                "finder-pattern centres (x, y)",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "count, module_size (mean, pixels)",
            ),
        ]
    }

    fn new(p: QrFinderParams) -> Result<Self, String> {
        if !(-1..=255).contains(&p.threshold) {
            return Err(format!(
                "`threshold` must be -1 or 0..=255, got {}",
                p.threshold
            ));
        }
        if !p.tolerance.is_finite() || !(0.05..=1.0).contains(&p.tolerance) {
            return Err(format!(
                "`tolerance` must be in [0.05, 1], got {}",
                p.tolerance
            ));
        }
        if p.min_confirmations == 0 {
            return Err("`min_confirmations` must be ≥ 1".into());
        }
        Ok(QrFinder {
            threshold: u8::try_from(p.threshold).ok(),
            tolerance: p.tolerance,
            min_confirmations: p.min_confirmations,
        })
    }
}

impl Operator for QrFinder {
    fn run(&self, _ctx: &RunContext, inputs: &Inputs<'_>) -> Result<Outputs, OpError> {
        let image = inputs.image("image")?;
        let gray = gray_u8(image);
        let found = qr_finders(
            &gray,
            image.width(),
            image.height(),
            self.threshold,
            self.tolerance,
            self.min_confirmations,
        );
        let mut metrics = Metrics::new();
        metrics.insert("count".into(), found.len() as f64);
        let module = if found.is_empty() {
            0.0
        } else {
            found.iter().map(|f| f.module).sum::<f64>() / found.len() as f64
        };
        metrics.insert("module_size".into(), module);
        let points: Vec<[f64; 2]> = found.iter().map(|f| [f.x, f.y]).collect();
        Ok(Outputs::new()
            .with("centres", Value::Points2D(Arc::new(points)))
            .with("metrics", Value::metrics(metrics)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ocellus_engine::params::{ParamValue, Params};
    use ocellus_engine::value::{Channels, Image};

    /// A 25×25-module QR-like symbol: three finder patterns with white separators, random
    /// modules elsewhere. `true` = dark.
    fn symbol(seed: u64) -> Vec<bool> {
        let n = 25;
        let mut state = seed | 1;
        let mut m: Vec<bool> = (0..n * n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state & 1 == 1
            })
            .collect();
        for (ox, oy) in [(0, 0), (n - 7, 0), (0, n - 7)] {
            for y in 0..8usize {
                for x in 0..8usize {
                    // Separator included (modules 7 on the inner sides).
                    let (gx, gy) = (
                        if ox == 0 { x } else { ox + x - 1 },
                        if oy == 0 { y } else { oy + y - 1 },
                    );
                    if gx >= n || gy >= n {
                        continue;
                    }
                    let (lx, ly) = (gx as isize - ox as isize, gy as isize - oy as isize);
                    let inside = (0..7).contains(&lx) && (0..7).contains(&ly);
                    let dark = inside && {
                        let ring = lx.min(ly).min(6 - lx).min(6 - ly);
                        ring != 1
                    };
                    m[gy * n + gx] = dark;
                }
            }
        }
        m
    }

    /// Renders the symbol with a 4-module quiet zone: module size `s` pixels, rotated by
    /// `angle` about the image centre, 4×4 supersampled. Returns the image and the finder
    /// centres (pixel centres at integers).
    fn render(s: f64, angle: f64, seed: u64) -> (Vec<u8>, usize, usize, Vec<[f64; 2]>) {
        let n = 25.0;
        let side = ((n + 8.0) * s * 1.5).ceil() as usize;
        let (w, h) = (side, side);
        let m = symbol(seed);
        let (c, sn) = (angle.cos(), angle.sin());
        let centre = side as f64 / 2.0;
        // Module coordinates (u, v) ↔ image: p = centre + R · ((u − n/2) s, (v − n/2) s).
        let to_image = |u: f64, v: f64| {
            let (a, b) = ((u - n / 2.0) * s, (v - n / 2.0) * s);
            [centre + c * a - sn * b, centre + sn * a + c * b]
        };
        let mut img = vec![0u8; w * h];
        let k = 4;
        for y in 0..h {
            for x in 0..w {
                let mut dark = 0;
                for j in 0..k {
                    for i in 0..k {
                        let px = x as f64 + (i as f64 + 0.5) / k as f64 - centre;
                        let py = y as f64 + (j as f64 + 0.5) / k as f64 - centre;
                        let u = (c * px + sn * py) / s + n / 2.0;
                        let v = (-sn * px + c * py) / s + n / 2.0;
                        if u >= 0.0 && v >= 0.0 && u < n && v < n && m[v as usize * 25 + u as usize]
                        {
                            dark += 1;
                        }
                    }
                }
                img[y * w + x] = (230 - 200 * dark / (k * k)) as u8;
            }
        }
        let truth = [(3.5, 3.5), (21.5, 3.5), (3.5, 21.5)]
            .iter()
            .map(|&(u, v)| {
                let p = to_image(u, v);
                [p[0] - 0.5, p[1] - 0.5]
            })
            .collect();
        (img, w, h, truth)
    }

    fn check(s: f64, angle: f64, seed: u64) {
        let (img, w, h, truth) = render(s, angle, seed);
        let found = qr_finders(&img, w, h, None, 0.5, 2);
        for t in &truth {
            let best = found
                .iter()
                .map(|f| (f.x - t[0]).hypot(f.y - t[1]))
                .fold(f64::INFINITY, f64::min);
            assert!(
                best < 1.0,
                "scale {s}, angle {angle}: centre {t:?} missed by {best}; found {found:?}"
            );
        }
        assert_eq!(found.len(), 3, "scale {s}, angle {angle}: {found:?}");
        for f in &found {
            assert!(
                (f.module - s).abs() < 0.25 * s,
                "module {} vs {s}",
                f.module
            );
        }
    }

    #[test]
    fn finds_three_centres_at_several_scales() {
        for (i, s) in [3.0, 4.5, 7.0].into_iter().enumerate() {
            check(s, 0.0, 11 + i as u64);
        }
    }

    #[test]
    fn finds_three_centres_rotated() {
        check(5.0, 0.35, 7);
        check(6.0, -0.6, 8);
    }

    #[test]
    fn ratio_signature() {
        assert!(ratio_ok(&[2, 2, 6, 2, 2], 0.5));
        assert!(ratio_ok(&[3, 2, 7, 2, 3], 0.5));
        assert!(!ratio_ok(&[2, 2, 2, 2, 2], 0.5));
        assert!(!ratio_ok(&[6, 2, 6, 2, 2], 0.5));
        assert!(!ratio_ok(&[0, 2, 6, 2, 2], 0.5));
    }

    #[test]
    fn otsu_splits_two_levels() {
        let mut v = vec![20u8; 50];
        v.extend(vec![200u8; 50]);
        let t = otsu_threshold(&v);
        assert!((20..200).contains(&t));
        assert_eq!(otsu_threshold(&[5, 5, 5]), 0);
    }

    #[test]
    fn empty_constant_and_operator() {
        assert!(qr_finders(&[], 0, 0, None, 0.5, 2).is_empty());
        assert!(qr_finders(&[9], 1, 1, None, 0.5, 2).is_empty());
        assert!(qr_finders(&[128; 100], 10, 10, None, 0.5, 1).is_empty());
        let (img, w, h, truth) = render(4.0, 0.0, 3);
        let rgb: Vec<f32> = img
            .iter()
            .flat_map(|&v| [f32::from(v) / 255.0; 3])
            .collect();
        let op = QrFinder::new(QrFinderParams::default()).unwrap();
        let specs = QrFinder::inputs();
        let values = [Some(Value::image(
            Image::from_f32(w, h, Channels::Rgb, rgb).unwrap(),
        ))];
        let ctx = RunContext {
            node: "qr".into(),
            threads: 1,
            element: None,
        };
        let mut out = op.run(&ctx, &Inputs::new(&specs, &values)).unwrap();
        let Some(Value::Points2D(p)) = out.take("centres") else {
            panic!("no centres")
        };
        assert_eq!(p.len(), truth.len());
        let Some(Value::Metrics(m)) = out.take("metrics") else {
            panic!("no metrics")
        };
        assert_eq!(m["count"], 3.0);
        assert!((m["module_size"] - 4.0).abs() < 0.5);
        let mut bad = QrFinderParams::default().to_map();
        bad.insert("tolerance".into(), ParamValue::Float(f64::NAN));
        assert!(
            QrFinderParams::from_map(&bad)
                .map(|p| QrFinder::new(p).is_err())
                .unwrap_or(true)
        );
        assert!(
            QrFinder::new(QrFinderParams {
                threshold: 300,
                ..QrFinderParams::default()
            })
            .is_err()
        );
    }
}
