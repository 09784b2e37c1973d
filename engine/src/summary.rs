//! Stable, human-readable summaries of values for snapshot tests.
//!
//! [`summarize_outputs`] renders a graph's outputs as RON-like text, one output per entry:
//!
//! ```text
//! (
//!     "edges": Image(width: 1920, height: 1080, format: "gray_u8", min: [0], mean: [12.3456], max: [255], dhash: "0x1f3a5b7c9d0e2f41"),
//!     "stats": Metrics({
//!         "gray.mean": 104.512,
//!     }),
//! )
//! ```
//!
//! Rules that keep snapshots stable and reviewable:
//! - every float goes through [`fmt_sig6`] (6 significant digits, C's `%g`);
//! - statistics are computed sequentially in a fixed order in `f64`, never in parallel, so the
//!   text is the same whatever the thread count;
//! - statistics of float data skip non-finite entries and report how many there were as
//!   `non_finite: N` (left out when zero);
//! - images carry a 64-bit perceptual difference hash ([`dhash`]) so a changed picture shows up
//!   even when its statistics barely move;
//! - values with many parts (metrics, lists, small matrices) are written as indented blocks, all
//!   others on one line.
//!
//! The text is meant for reading and diffing; it is RON-shaped but not meant to be parsed back.

use std::fmt::Write as _;

use crate::value::{
    Animation, Camera, Descriptors, Distortion, Image, Keypoint, Match, Matrix, Mesh, Metrics,
    PixelData, PointCloud, Pose, Reconstruction, Scene, Tracks, Value, ValueList,
};

/// Indentation step of nested blocks.
const INDENT: usize = 4;

/// Matrices with at most this many entries are printed in full.
const MATRIX_FULL_ENTRIES: usize = 16;

/// Text longer than this many characters is truncated.
const TEXT_MAX_CHARS: usize = 200;

/// dHash grid: luminance is averaged down to `DHASH_COLS × DHASH_ROWS` cells and each row gives
/// `DHASH_COLS - 1` comparison bits.
const DHASH_COLS: usize = 9;
/// See [`DHASH_COLS`].
const DHASH_ROWS: usize = 8;

/// Rec. 709 luma weights for r, g, b.
const LUMA_WEIGHTS: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Formats a float with 6 significant digits, like C's `printf("%g")`: fixed notation for
/// decimal exponents -4..=5 (`104.512`, `0.000123457`), scientific otherwise (`1.23457e+09`,
/// `1e-05`), trailing zeros removed. `-0` prints as `0`, NaN as `NaN`, infinities as `inf` and
/// `-inf`.
pub fn fmt_sig6(x: f64) -> String {
    if x.is_nan() {
        return "NaN".to_string();
    }
    if x.is_infinite() {
        return if x > 0.0 { "inf" } else { "-inf" }.to_string();
    }
    if x == 0.0 {
        return "0".to_string();
    }
    // The exponent after rounding to 6 significant digits decides the notation, as in C.
    let scientific = format!("{x:.5e}");
    let Some((mantissa, exponent)) = scientific.split_once('e') else {
        return scientific;
    };
    let Ok(exponent) = exponent.parse::<i32>() else {
        return scientific;
    };
    if !(-4..6).contains(&exponent) {
        let sign = if exponent < 0 { '-' } else { '+' };
        format!(
            "{}e{sign}{:02}",
            strip_fraction_zeros(mantissa),
            exponent.unsigned_abs()
        )
    } else {
        let decimals = usize::try_from(5 - exponent).unwrap_or(0);
        strip_fraction_zeros(&format!("{x:.decimals$}")).to_string()
    }
}

fn strip_fraction_zeros(s: &str) -> &str {
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.')
    } else {
        s
    }
}

/// 64-bit difference hash of an image, or `None` for a zero-area image.
///
/// The image is converted to luminance (gray as is; rgb/rgba with Rec. 709 weights, alpha
/// ignored; samples at their stored scale), area-averaged down to 9 × 8 cells with exact
/// fractional pixel coverage (so images smaller than 9 × 8 are well-defined: their pixels are
/// spread over several cells), and bit `i = 8·row + col` (`col < 8`) is set when cell
/// `(row, col)` is darker than cell `(row, col + 1)`. Bit 0 is the most significant, so the hex
/// digits read like the image, top-left first. Scaling all samples by a positive factor does not
/// change the hash.
pub fn dhash(image: &Image) -> Option<u64> {
    if image.is_empty() {
        return None;
    }
    let (w, h) = (image.width(), image.height());
    let col_weights = coverage(w, DHASH_COLS);
    let row_weights = coverage(h, DHASH_ROWS);
    let mut cells = [[0.0f64; DHASH_COLS]; DHASH_ROWS];
    let mut row_sums = [0.0f64; DHASH_COLS];
    let channels = image.channels().count();
    for (y, y_weights) in row_weights.iter().enumerate() {
        row_sums.fill(0.0);
        for (x, x_weights) in col_weights.iter().enumerate() {
            let l = luminance(image, (y * w + x) * channels, channels);
            for &(cell, weight) in x_weights {
                row_sums[cell] += weight * l;
            }
        }
        for &(cell_row, weight) in y_weights {
            for (acc, sum) in cells[cell_row].iter_mut().zip(&row_sums) {
                *acc += weight * sum;
            }
        }
    }
    // Every cell covers the same total weight, so sums compare like averages.
    let mut hash = 0u64;
    for row in &cells {
        for pair in row.windows(2) {
            hash <<= 1;
            if pair[0] < pair[1] {
                hash |= 1;
            }
        }
    }
    Some(hash)
}

/// For each of `n_in` source pixels, the output cells it overlaps and by how much, when `n_out`
/// cells evenly cover the source. Computed in units of `1 / (n_in · n_out)` pixel, so weights are
/// exact integers.
fn coverage(n_in: usize, n_out: usize) -> Vec<Vec<(usize, f64)>> {
    let (n_in64, n_out64) = (n_in as u64, n_out as u64);
    (0..n_in64)
        .map(|i| {
            let (lo, hi) = (i * n_out64, (i + 1) * n_out64);
            let first = lo / n_in64;
            let last = (hi - 1) / n_in64;
            (first..=last)
                .map(|cell| {
                    let overlap = hi.min((cell + 1) * n_in64) - lo.max(cell * n_in64);
                    (cell as usize, overlap as f64)
                })
                .collect()
        })
        .collect()
}

fn luminance(image: &Image, start: usize, channels: usize) -> f64 {
    let sample = |i: usize| -> f64 {
        match image.data() {
            PixelData::U8(v) => v.get(start + i).map_or(0.0, |s| f64::from(*s)),
            PixelData::U16(v) => v.get(start + i).map_or(0.0, |s| f64::from(*s)),
            PixelData::F32(v) => v.get(start + i).map_or(0.0, |s| f64::from(*s)),
        }
    };
    if channels == 1 {
        sample(0)
    } else {
        LUMA_WEIGHTS
            .iter()
            .enumerate()
            .map(|(i, w)| w * sample(i))
            .sum()
    }
}

/// Running statistics in a fixed order; non-finite entries are counted, not summed.
#[derive(Debug, Clone, Copy)]
struct Stats {
    count: u64,
    non_finite: u64,
    min: f64,
    max: f64,
    sum: f64,
}

impl Stats {
    fn new() -> Stats {
        Stats {
            count: 0,
            non_finite: 0,
            min: f64::INFINITY,
            max: f64::NEG_INFINITY,
            sum: 0.0,
        }
    }

    fn of(values: impl IntoIterator<Item = f64>) -> Stats {
        let mut s = Stats::new();
        values.into_iter().for_each(|v| s.push(v));
        s
    }

    fn push(&mut self, v: f64) {
        if v.is_finite() {
            self.count += 1;
            self.min = self.min.min(v);
            self.max = self.max.max(v);
            self.sum += v;
        } else {
            self.non_finite += 1;
        }
    }

    fn min(&self) -> f64 {
        if self.count == 0 { f64::NAN } else { self.min }
    }

    fn max(&self) -> f64 {
        if self.count == 0 { f64::NAN } else { self.max }
    }

    fn mean(&self) -> f64 {
        if self.count == 0 {
            f64::NAN
        } else {
            self.sum / self.count as f64
        }
    }

    /// `(min: a, mean: b, max: c)`, plus `non_finite: n` when there were any.
    fn triple(&self) -> String {
        let mut s = format!(
            "(min: {}, mean: {}, max: {}",
            fmt_sig6(self.min()),
            fmt_sig6(self.mean()),
            fmt_sig6(self.max())
        );
        push_non_finite(&mut s, self.non_finite);
        s.push(')');
        s
    }
}

fn push_non_finite(s: &mut String, n: u64) {
    if n > 0 {
        let _ = write!(s, ", non_finite: {n}");
    }
}

/// `[a, b, c]` with [`fmt_sig6`] entries.
fn list_f64(values: impl IntoIterator<Item = f64>) -> String {
    let items: Vec<String> = values.into_iter().map(fmt_sig6).collect();
    format!("[{}]", items.join(", "))
}

/// A RON string literal: quotes, backslashes and control characters escaped.
fn ron_string(text: &str) -> String {
    let mut out = String::with_capacity(text.len() + 2);
    out.push('"');
    for c in text.chars() {
        match c {
            '"' => out.push_str("\\\""),
            '\\' => out.push_str("\\\\"),
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if c.is_control() => {
                let _ = write!(out, "\\u{{{:x}}}", u32::from(c));
            }
            c => out.push(c),
        }
    }
    out.push('"');
    out
}

/// Summary of one value. Single-line for most values; metrics, lists and small matrices are
/// blocks whose inner lines are indented by four spaces and whose closing line is not indented.
pub fn summarize_value(value: &Value) -> String {
    let mut out = String::new();
    write_value(&mut out, value, 0);
    out
}

/// Summary of named outputs in the given order:
///
/// ```text
/// (
///     "name": <summarize_value>,
/// )
/// ```
///
/// The text ends with a newline; an empty slice gives `()` and a newline.
pub fn summarize_outputs(outputs: &[(String, Value)]) -> String {
    if outputs.is_empty() {
        return "()\n".to_string();
    }
    let mut out = String::from("(\n");
    for (name, value) in outputs {
        pad(&mut out, INDENT);
        out.push_str(&ron_string(name));
        out.push_str(": ");
        write_value(&mut out, value, INDENT);
        out.push_str(",\n");
    }
    out.push_str(")\n");
    out
}

fn pad(out: &mut String, indent: usize) {
    out.extend(std::iter::repeat_n(' ', indent));
}

/// Appends the summary of `value`, whose first line is already indented by `indent`.
fn write_value(out: &mut String, value: &Value, indent: usize) {
    match value {
        Value::Image(image) => out.push_str(&image_summary(image)),
        Value::Keypoints(k) => out.push_str(&keypoints_summary(k)),
        Value::Descriptors(d) => out.push_str(&descriptors_summary(d)),
        Value::Matches(m) => out.push_str(&matches_summary(m)),
        Value::Matrix(m) => write_matrix(out, m, indent),
        Value::Camera(c) => out.push_str(&camera_summary(c)),
        Value::Pose(p) => out.push_str(&pose_summary(p)),
        Value::Points2D(p) => out.push_str(&points2d_summary(p)),
        Value::PointCloud(p) => out.push_str(&point_cloud_summary(p)),
        Value::Tracks(t) => out.push_str(&tracks_summary(t)),
        Value::Reconstruction(r) => out.push_str(&reconstruction_summary(r)),
        Value::Mesh(m) => out.push_str(&format!("Mesh({})", mesh_fields(m))),
        Value::Bvh(b) => {
            let stats = b.stats();
            let _ = write!(
                out,
                "Bvh(triangles: {}, nodes: {}, leaves: {}, max_depth: {}, max_leaf_size: {})",
                b.primitives.len(),
                stats.nodes,
                stats.leaves,
                stats.max_depth,
                stats.max_leaf_size
            );
        }
        Value::Scene(s) => out.push_str(&scene_summary(s)),
        Value::Animation(a) => out.push_str(&animation_summary(a)),
        Value::Scalar(x) => {
            let _ = write!(out, "Scalar({})", fmt_sig6(*x));
        }
        Value::Integer(i) => {
            let _ = write!(out, "Integer({i})");
        }
        Value::Bool(b) => {
            let _ = write!(out, "Bool({b})");
        }
        Value::Text(t) => out.push_str(&text_summary(t)),
        Value::Metrics(m) => write_metrics(out, m, indent),
        Value::List(l) => write_list(out, l, indent),
    }
}

fn image_summary(image: &Image) -> String {
    let mut s = format!(
        "Image(width: {}, height: {}, format: \"{}\"",
        image.width(),
        image.height(),
        image.format()
    );
    if image.is_empty() {
        s.push_str(", dhash: \"none\")");
        return s;
    }
    let channels = image.channels().count();
    let stats: Vec<Stats> = (0..channels)
        .map(|c| match image.data() {
            PixelData::U8(v) => {
                Stats::of(v.iter().skip(c).step_by(channels).map(|&x| f64::from(x)))
            }
            PixelData::U16(v) => {
                Stats::of(v.iter().skip(c).step_by(channels).map(|&x| f64::from(x)))
            }
            PixelData::F32(v) => {
                Stats::of(v.iter().skip(c).step_by(channels).map(|&x| f64::from(x)))
            }
        })
        .collect();
    let _ = write!(
        s,
        ", min: {}, mean: {}, max: {}",
        list_f64(stats.iter().map(Stats::min)),
        list_f64(stats.iter().map(Stats::mean)),
        list_f64(stats.iter().map(Stats::max))
    );
    push_non_finite(&mut s, stats.iter().map(|st| st.non_finite).sum());
    let hash = dhash(image).map_or_else(|| "none".to_string(), |h| format!("0x{h:016x}"));
    let _ = write!(s, ", dhash: \"{hash}\")");
    s
}

fn keypoints_summary(keypoints: &[Keypoint]) -> String {
    if keypoints.is_empty() {
        return "Keypoints(count: 0)".to_string();
    }
    let field = |f: fn(&Keypoint) -> f32| Stats::of(keypoints.iter().map(|k| f64::from(f(k))));
    let (x, y) = (field(|k| k.x), field(|k| k.y));
    format!(
        "Keypoints(count: {}, min: {}, max: {}, size: {}, response: {})",
        keypoints.len(),
        list_f64([x.min(), y.min()]),
        list_f64([x.max(), y.max()]),
        field(|k| k.size).triple(),
        field(|k| k.response).triple()
    )
}

fn descriptors_summary(descriptors: &Descriptors) -> String {
    match descriptors {
        Descriptors::Float { dim, data } => {
            let mut s = format!(
                "Descriptors(kind: \"float\", count: {}, dim: {dim}",
                descriptors.len()
            );
            if !data.is_empty() {
                let values = Stats::of(data.iter().map(|&v| f64::from(v)));
                let norms = Stats::of(data.chunks(*dim.max(&1)).map(|row| {
                    row.iter()
                        .map(|&v| f64::from(v) * f64::from(v))
                        .sum::<f64>()
                        .sqrt()
                }));
                let _ = write!(
                    s,
                    ", values: {}, mean_norm: {}",
                    values.triple(),
                    fmt_sig6(norms.mean())
                );
            }
            s.push(')');
            s
        }
        Descriptors::Binary { bytes, data } => {
            let mut s = format!(
                "Descriptors(kind: \"binary\", count: {}, bytes: {bytes}",
                descriptors.len()
            );
            if !descriptors.is_empty() {
                let bits: u64 = data.iter().map(|b| u64::from(b.count_ones())).sum();
                let _ = write!(
                    s,
                    ", mean_bits_set: {}",
                    fmt_sig6(bits as f64 / descriptors.len() as f64)
                );
            }
            s.push(')');
            s
        }
    }
}

fn matches_summary(matches: &[Match]) -> String {
    if matches.is_empty() {
        return "Matches(count: 0)".to_string();
    }
    format!(
        "Matches(count: {}, distance: {})",
        matches.len(),
        Stats::of(matches.iter().map(|m| f64::from(m.distance))).triple()
    )
}

fn write_matrix(out: &mut String, m: &Matrix, indent: usize) {
    let _ = write!(out, "Matrix(rows: {}, cols: {}", m.rows, m.cols);
    if m.data.len() <= MATRIX_FULL_ENTRIES {
        if m.data.is_empty() || m.cols == 0 {
            out.push_str(", data: [])");
            return;
        }
        out.push_str(", data: [\n");
        for row in m.data.chunks(m.cols) {
            pad(out, indent + INDENT);
            out.push_str(&list_f64(row.iter().copied()));
            out.push_str(",\n");
        }
        pad(out, indent);
        out.push_str("])");
    } else {
        let stats = Stats::of(m.data.iter().copied());
        let frobenius = m
            .data
            .iter()
            .filter(|v| v.is_finite())
            .map(|v| v * v)
            .sum::<f64>()
            .sqrt();
        let _ = write!(
            out,
            ", min: {}, mean: {}, max: {}, frobenius: {}",
            fmt_sig6(stats.min()),
            fmt_sig6(stats.mean()),
            fmt_sig6(stats.max()),
            fmt_sig6(frobenius)
        );
        push_non_finite(out, stats.non_finite);
        out.push(')');
    }
}

fn camera_summary(camera: &Camera) -> String {
    let k = camera.intrinsics();
    let distortion = match camera.distortion() {
        Distortion::None => "none".to_string(),
        Distortion::RadialTangential(d) => format!("radial_tangential {}", list_f64(d)),
        Distortion::Fisheye(d) => format!("fisheye {}", list_f64(d)),
    };
    format!(
        "Camera(width: {}, height: {}, fx: {}, fy: {}, cx: {}, cy: {}, skew: {}, distortion: \"{distortion}\")",
        camera.width,
        camera.height,
        fmt_sig6(k.fx),
        fmt_sig6(k.fy),
        fmt_sig6(k.cx),
        fmt_sig6(k.cy),
        fmt_sig6(k.skew),
    )
}

fn pose_summary(pose: &Pose) -> String {
    format!(
        "Pose(rotation: {}, translation: {})",
        list_f64(pose.rotation_matrix()),
        list_f64(pose.translation)
    )
}

fn points2d_summary(points: &[[f64; 2]]) -> String {
    if points.is_empty() {
        return "Points2D(count: 0)".to_string();
    }
    let axes: Vec<Stats> = (0..2)
        .map(|a| Stats::of(points.iter().map(|p| p[a])))
        .collect();
    format!(
        "Points2D(count: {}, {})",
        points.len(),
        bounds_fields(&axes)
    )
}

/// `min: [..], max: [..], centroid: [..]` (+ `non_finite`) over per-axis statistics.
fn bounds_fields(axes: &[Stats]) -> String {
    let mut s = format!(
        "min: {}, max: {}, centroid: {}",
        list_f64(axes.iter().map(Stats::min)),
        list_f64(axes.iter().map(Stats::max)),
        list_f64(axes.iter().map(Stats::mean))
    );
    push_non_finite(&mut s, axes.iter().map(|a| a.non_finite).sum());
    s
}

fn positions_bounds(positions: &[[f32; 3]]) -> String {
    let axes: Vec<Stats> = (0..3)
        .map(|a| Stats::of(positions.iter().map(|p| f64::from(p[a]))))
        .collect();
    bounds_fields(&axes)
}

fn point_cloud_summary(cloud: &PointCloud) -> String {
    let mut s = format!("PointCloud(count: {}", cloud.positions.len());
    if !cloud.positions.is_empty() {
        let _ = write!(s, ", {}", positions_bounds(&cloud.positions));
    }
    let _ = write!(
        s,
        ", colors: {}, normals: {})",
        cloud.colors.is_some(),
        cloud.normals.is_some()
    );
    s
}

fn mesh_fields(mesh: &Mesh) -> String {
    let mut s = format!(
        "vertices: {}, triangles: {}",
        mesh.positions.len(),
        mesh.triangles.len()
    );
    if !mesh.positions.is_empty() {
        let _ = write!(s, ", {}", positions_bounds(&mesh.positions));
    }
    let _ = write!(
        s,
        ", normals: {}, uvs: {}, colors: {}",
        mesh.normals.is_some(),
        mesh.uvs.is_some(),
        mesh.colors.is_some()
    );
    if mesh.tangents.is_some() {
        s.push_str(", tangents: true");
    }
    s
}

fn tracks_summary(tracks: &Tracks) -> String {
    if tracks.tracks.is_empty() {
        return "Tracks(count: 0)".to_string();
    }
    let observations: usize = tracks.tracks.iter().map(Vec::len).sum();
    format!(
        "Tracks(count: {}, observations: {observations}, length: {})",
        tracks.tracks.len(),
        Stats::of(tracks.tracks.iter().map(|t| t.len() as f64)).triple()
    )
}

fn reconstruction_summary(r: &Reconstruction) -> String {
    let observations: usize = r.points.iter().map(|p| p.track.len()).sum();
    let mut s = format!(
        "Reconstruction(cameras: {}, images: {}, points: {}, observations: {observations}",
        r.cameras.len(),
        r.images.len(),
        r.points.len()
    );
    if !r.points.is_empty() {
        let errors = Stats::of(r.points.iter().map(|p| p.error_px));
        let _ = write!(
            s,
            ", mean_track_length: {}, mean_error_px: {}",
            fmt_sig6(observations as f64 / r.points.len() as f64),
            fmt_sig6(errors.mean())
        );
        push_non_finite(&mut s, errors.non_finite);
    }
    s.push(')');
    s
}

fn scene_summary(scene: &Scene) -> String {
    let (vertices, triangles) = scene.mesh_counts();
    let names: Vec<String> = scene.objects.iter().map(|o| ron_string(&o.name)).collect();
    format!(
        "Scene(objects: {}, materials: {}, vertices: {vertices}, triangles: {triangles}, lights: {}, cameras: {}, names: [{}])",
        scene.objects.len(),
        scene.materials.len(),
        scene.lights.len(),
        scene.cameras.len(),
        names.join(", ")
    )
}

fn animation_summary(animation: &Animation) -> String {
    let keyframes: usize = animation.channels.iter().map(|c| c.times.len()).sum();
    let targets: Vec<String> = animation
        .channels
        .iter()
        .map(|c| ron_string(&c.target))
        .collect();
    format!(
        "Animation(duration: {}, channels: {}, keyframes: {keyframes}, targets: [{}])",
        fmt_sig6(animation.duration),
        animation.channels.len(),
        targets.join(", ")
    )
}

fn text_summary(text: &str) -> String {
    let total = text.chars().count();
    if total <= TEXT_MAX_CHARS {
        format!("Text({})", ron_string(text))
    } else {
        let head: String = text.chars().take(TEXT_MAX_CHARS).collect();
        format!("Text({}, total_chars: {total})", ron_string(&head))
    }
}

fn write_metrics(out: &mut String, metrics: &Metrics, indent: usize) {
    if metrics.is_empty() {
        out.push_str("Metrics({})");
        return;
    }
    out.push_str("Metrics({\n");
    for (name, value) in metrics {
        pad(out, indent + INDENT);
        let _ = writeln!(out, "{}: {},", ron_string(name), fmt_sig6(*value));
    }
    pad(out, indent);
    out.push_str("})");
}

fn write_list(out: &mut String, list: &ValueList, indent: usize) {
    let _ = write!(
        out,
        "List(element: \"{}\", len: {}, items: [",
        list.element,
        list.items.len()
    );
    if list.items.is_empty() {
        out.push_str("])");
        return;
    }
    out.push('\n');
    for item in &list.items {
        pad(out, indent + INDENT);
        write_value(out, item, indent + INDENT);
        out.push_str(",\n");
    }
    pad(out, indent);
    out.push_str("])");
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::types::PortType;
    use crate::value::{CameraModel, Channels};

    #[test]
    fn fmt_sig6_matches_printf_g() {
        let cases: [(f64, &str); 28] = [
            (0.0, "0"),
            (-0.0, "0"),
            (1.0, "1"),
            (-2.5, "-2.5"),
            (104.512, "104.512"),
            (104.5123, "104.512"),
            (0.1, "0.1"),
            (1.0 / 3.0, "0.333333"),
            (2.0 / 3.0, "0.666667"),
            (0.000123456789, "0.000123457"),
            (0.0001, "0.0001"),
            (0.00001, "1e-05"),
            (0.0000123456, "1.23456e-05"),
            (100000.0, "100000"),
            (123456.7, "123457"),
            (999999.0, "999999"),
            (999999.5, "1e+06"),
            (1000000.0, "1e+06"),
            (1234567890.0, "1.23457e+09"),
            (-1234567890.0, "-1.23457e+09"),
            (9.9999996, "10"),
            (1e100, "1e+100"),
            (1.5e-300, "1.5e-300"),
            (5e-324, "4.94066e-324"),
            (f64::MAX, "1.79769e+308"),
            (f64::NAN, "NaN"),
            (f64::INFINITY, "inf"),
            (f64::NEG_INFINITY, "-inf"),
        ];
        for (x, expected) in cases {
            assert_eq!(fmt_sig6(x), expected, "{x:e}");
        }
    }

    fn gradient(w: usize, h: usize, scale: f32) -> Image {
        let data = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                (x * 3 + y) as f32 * scale
            })
            .collect();
        Image::from_f32(w, h, Channels::Gray, data).unwrap()
    }

    #[test]
    fn dhash_ignores_brightness_scaling_but_not_flips() {
        let base = dhash(&gradient(40, 30, 1.0)).unwrap();
        assert_eq!(base, u64::MAX, "a left-to-right ramp sets every bit");
        assert_eq!(dhash(&gradient(40, 30, 0.37)), Some(base));
        assert_eq!(dhash(&gradient(40, 30, 250.0)), Some(base));

        // u8 image: a non-monotone pattern, then the same pattern brighter.
        let pattern: Vec<u8> = (0..64 * 48)
            .map(|i| {
                let (x, y) = (i % 64, i / 64);
                ((x * 7 + y * 13) % 50 + (x / 8) * 5) as u8
            })
            .collect();
        let dim = Image::from_u8(64, 48, Channels::Gray, pattern.clone()).unwrap();
        let bright = Image::from_u8(
            64,
            48,
            Channels::Gray,
            pattern.iter().map(|v| v * 2).collect(),
        )
        .unwrap();
        assert_eq!(dhash(&dim), dhash(&bright));

        // Mirrored left-right: every comparison flips.
        let flipped: Vec<f32> = {
            let g = gradient(40, 30, 1.0);
            let d = g.as_f32().unwrap();
            (0..40 * 30)
                .map(|i| d[(i / 40) * 40 + 39 - i % 40])
                .collect()
        };
        let flipped = Image::from_f32(40, 30, Channels::Gray, flipped).unwrap();
        assert_eq!(dhash(&flipped), Some(0));
        assert_ne!(
            dhash(&dim),
            dhash(&{
                let d: Vec<u8> = (0..64 * 48)
                    .map(|i| pattern[(i / 64) * 64 + 63 - i % 64])
                    .collect();
                Image::from_u8(64, 48, Channels::Gray, d).unwrap()
            })
        );
    }

    #[test]
    fn dhash_small_and_empty_images() {
        // 2×1: cells 0..=3 see pixel 0 (10), cell 4 straddles (15), cells 5..=8 see pixel 1 (20):
        // bits for cols 3 and 4 in every row, i.e. 0b0001_1000 per row.
        let tiny = Image::from_u8(2, 1, Channels::Gray, vec![10, 20]).unwrap();
        assert_eq!(dhash(&tiny), Some(0x1818_1818_1818_1818));
        let single = Image::from_u8(1, 1, Channels::Rgb, vec![1, 2, 3]).unwrap();
        assert_eq!(dhash(&single), Some(0));
        let empty = Image::from_u8(0, 4, Channels::Gray, vec![]).unwrap();
        assert_eq!(dhash(&empty), None);
    }

    #[test]
    fn coverage_weights_sum_per_cell() {
        for (n_in, n_out) in [(1, 9), (2, 9), (9, 9), (10, 9), (1000, 8), (7, 8)] {
            let mut per_cell = vec![0.0; n_out];
            for pixel in coverage(n_in, n_out) {
                for (cell, w) in pixel {
                    per_cell[cell] += w;
                }
            }
            assert!(
                per_cell.iter().all(|&w| w == n_in as f64),
                "{n_in}->{n_out}"
            );
        }
    }

    #[test]
    fn known_image_summary() {
        // 2×1 rgb: pixel 0 = (0, 10, 200), pixel 1 = (255, 20, 100).
        let image = Image::from_u8(2, 1, Channels::Rgb, vec![0, 10, 200, 255, 20, 100]).unwrap();
        // Luma: 0.2126·0 + 0.7152·10 + 0.0722·200 = 21.592 < 0.2126·255 + 0.7152·20 + 0.0722·100
        // = 75.083, so the hash is the same as the gray 10 → 20 case.
        assert_eq!(
            summarize_value(&Value::image(image)),
            "Image(width: 2, height: 1, format: \"rgb_u8\", min: [0, 10, 100], mean: [127.5, 15, 150], max: [255, 20, 200], dhash: \"0x1818181818181818\")"
        );
        let empty = Image::from_f32(3, 0, Channels::Gray, vec![]).unwrap();
        assert_eq!(
            summarize_value(&Value::image(empty)),
            "Image(width: 3, height: 0, format: \"gray_f32\", dhash: \"none\")"
        );
        let nan = Image::from_f32(2, 1, Channels::Gray, vec![f32::NAN, 0.5]).unwrap();
        assert_eq!(
            summarize_value(&Value::image(nan)),
            "Image(width: 2, height: 1, format: \"gray_f32\", min: [0.5], mean: [0.5], max: [0.5], non_finite: 1, dhash: \"0x0000000000000000\")"
        );
    }

    #[test]
    fn outputs_layout() {
        let mut metrics = Metrics::new();
        metrics.insert("gray.mean".into(), 104.51234);
        metrics.insert("count".into(), 3.0);
        let matrix = Matrix::new(2, 2, vec![1.0, 0.5, -0.25, 1e-7]).unwrap();
        let outputs = vec![
            ("stats".to_string(), Value::metrics(metrics)),
            ("h".to_string(), Value::Matrix(Arc::new(matrix))),
            (
                "list".to_string(),
                Value::list(
                    PortType::Scalar.list_of(),
                    vec![
                        Value::list(PortType::Scalar, vec![Value::Scalar(1.0)]),
                        Value::list(PortType::Scalar, vec![]),
                    ],
                ),
            ),
            ("quote \"q\"".to_string(), Value::Text("a\nb".into())),
            ("n".to_string(), Value::Integer(-3)),
        ];
        let expected = r#"(
    "stats": Metrics({
        "count": 3,
        "gray.mean": 104.512,
    }),
    "h": Matrix(rows: 2, cols: 2, data: [
        [1, 0.5],
        [-0.25, 1e-07],
    ]),
    "list": List(element: "List<Scalar>", len: 2, items: [
        List(element: "Scalar", len: 1, items: [
            Scalar(1),
        ]),
        List(element: "Scalar", len: 0, items: []),
    ]),
    "quote \"q\"": Text("a\nb"),
    "n": Integer(-3),
)
"#;
        assert_eq!(summarize_outputs(&outputs), expected);
        assert_eq!(summarize_outputs(&[]), "()\n");
    }

    #[test]
    fn other_values() {
        let camera = Camera {
            model: CameraModel::Pinhole,
            width: 640,
            height: 480,
            params: vec![500.0, 500.0, 320.0, 240.0],
        };
        assert_eq!(
            summarize_value(&Value::Camera(Arc::new(camera))),
            "Camera(width: 640, height: 480, fx: 500, fy: 500, cx: 320, cy: 240, skew: 0, distortion: \"none\")"
        );
        assert_eq!(
            summarize_value(&Value::Pose(Pose::IDENTITY)),
            "Pose(rotation: [1, 0, 0, 0, 1, 0, 0, 0, 1], translation: [0, 0, 0])"
        );
        let cloud = PointCloud {
            positions: vec![[0.0, 0.0, 0.0], [2.0, 4.0, -1.0]],
            colors: None,
            normals: Some(vec![[0.0, 0.0, 1.0]; 2]),
        };
        assert_eq!(
            summarize_value(&Value::PointCloud(Arc::new(cloud))),
            "PointCloud(count: 2, min: [0, 0, -1], max: [2, 4, 0], centroid: [1, 2, -0.5], colors: false, normals: true)"
        );
        let big = Matrix::new(5, 5, (0..25).map(f64::from).collect()).unwrap();
        assert_eq!(
            summarize_value(&Value::Matrix(Arc::new(big))),
            "Matrix(rows: 5, cols: 5, min: 0, mean: 12, max: 24, frobenius: 70)"
        );
        let matches = vec![
            Match {
                query: 0,
                train: 1,
                distance: 1.0,
            },
            Match {
                query: 1,
                train: 0,
                distance: 3.0,
            },
        ];
        assert_eq!(
            summarize_value(&Value::Matches(Arc::new(matches))),
            "Matches(count: 2, distance: (min: 1, mean: 2, max: 3))"
        );
        let binary = Descriptors::Binary {
            bytes: 2,
            data: vec![0xFF, 0x00, 0x0F, 0x01],
        };
        assert_eq!(
            summarize_value(&Value::Descriptors(Arc::new(binary))),
            "Descriptors(kind: \"binary\", count: 2, bytes: 2, mean_bits_set: 6.5)"
        );
        let long: String = "é".repeat(250);
        let s = summarize_value(&Value::Text(long.into()));
        assert!(s.ends_with("\", total_chars: 250)"), "{s}");
        assert_eq!(s.chars().filter(|&c| c == 'é').count(), 200);
        assert_eq!(summarize_value(&Value::Bool(true)), "Bool(true)");
        assert_eq!(summarize_value(&Value::Scalar(f64::NAN)), "Scalar(NaN)");
        assert_eq!(
            summarize_value(&Value::Text("\u{1}\\".into())),
            "Text(\"\\u{1}\\\\\")"
        );
    }
}
